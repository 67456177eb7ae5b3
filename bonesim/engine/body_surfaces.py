"""Per-body surfaces: each body's voxels tessellated in its own frame.

Once a case's bone is split into several bodies (:mod:`bonesim.engine.bodies`),
one surface over the whole grid would join the bodies where they were cut
and draw every body where it was cut. :class:`BodySurfaces` keeps instead,
for every living body ``b``, a grid holding **only that body's voxels** and
a :class:`~bonesim.engine.surface.Surface` of it. A body's voxels never move
in the grid, so its surface lies in the body's own frame (vertex ``(i, j,
k)`` at ``origin + spacing * (i, j, k)`` [mm]); the body's pose
(``state.pose_m[b]``) places it in the case frame (the window sets it as
the actor's matrix).

Grids
-----
Every body grid uses the replica grid's lattice: voxel ``(i, j, k)`` means
the same voxel in each (same ``origin_mm``, ``spacing_mm``), so the voxel
lists of the tissue events apply to them unchanged.

Body 0 (the main bone)
    a full copy of the replica grid (sharing its brick table) in which the
    voxels of every other body have density 0. At the first split it takes
    over the one-body surface: the split voxels are simply *removed* from it
    by an incremental :meth:`Surface.update`, so the window keeps drawing
    the same surface object.
Any other body (a fragment)
    a :meth:`~bonesim.engine.grid.Grid.sub_grid` of the replica grid: only
    the bricks of the body's ``bounds`` plus :func:`margin_bricks` bricks
    around them (its surface closes, and every voxel its normals and
    thin-bone rays read is present), with the other bodies' voxels at
    density 0. A fragment costs memory in proportion to its box, never a
    full grid.

Every body grid holds the same labels as the replica grid (labels never
change), and a voxel's density is the replica's where the voxel belongs to
the body, 0 elsewhere. So each body's surface is exactly
``Surface.build`` of the replica grid with the other bodies' voxels emptied
(what the tests check).

Changes
-------
:meth:`BodySurfaces.update` takes one batch of applied events: the removed
voxels and the shading hints (touched) go to the body that holds them, the
voxels a ``SPLIT`` moved are removed from their source body, and a body
created or grown by a split is tessellated again from its grid (fragments
are small). Each body's grid is brought in step with the replica's tissue
for exactly those voxels (:func:`_sync_body`), then its surface is updated.
A ``POSE`` changes no geometry.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from bonesim.engine.bodies import BODY_LIMIT, voxel_bodies
from bonesim.engine.grid import BRICK, BRICK_SHIFT, Grid, find_brick, voxel_offset
from bonesim.engine.normals import NORMAL_RADIUS
from bonesim.engine.shading import load_shading
from bonesim.engine.surface import Surface
from bonesim.engine.thin_bone import tint_reach

__all__ = ["BodySurfaces", "margin_bricks", "masked_density"]

_NO_IJK = np.zeros((0, 3), np.int32)


@njit(cache=True, nogil=True)
def _sync_body(keys, vals, density, body, bid, bkeys, bvals, bdensity, ijk):
    # a body grid's voxel: the replica's density where it belongs to the body
    for q in range(ijk.shape[0]):
        i, j, k = ijk[q, 0], ijk[q, 1], ijk[q, 2]
        bb = find_brick(bkeys, bvals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        if bb < 0:
            continue
        off = voxel_offset(i, j, k)
        d = np.float32(0.0)
        g = find_brick(keys, vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT, k >> BRICK_SHIFT)
        if g >= 0 and body[g, off] == bid:
            d = density[g, off]
        bdensity[bb, off] = d


def _ijk(a) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.int32).reshape(-1, 3))


def masked_density(state, b: int, sel=None) -> np.ndarray:
    """The replica's density with every voxel not of body ``b`` at 0.

    Parameters
    ----------
    state : State
    b : int
        Body id.
    sel : (n_bricks,) bool, optional
        Only these bricks (default: all).

    Returns
    -------
    (n_sel, 512) float32
        A new array, laid out like ``state.grid.density[sel]``.
    """
    d = state.grid.density if sel is None else state.grid.density[sel]
    ids = state.body if sel is None else state.body[sel]
    return np.where(ids == b, d, np.float32(0.0)).astype(np.float32, copy=False)


def margin_bricks(spacing_mm: float, shading=None) -> int:
    """Bricks kept around a fragment's bounds in its grid.

    A vertex's normal reads densities within ``NORMAL_RADIUS`` voxels and
    its thin-bone rays within :func:`~bonesim.engine.thin_bone.tint_reach`;
    the shading's refresh windows reach ``2 NORMAL_RADIUS``. One voxel more
    closes the surface. Every voxel that far from the body must lie in an
    allocated brick of its grid, as it does in the replica grid.

    Parameters
    ----------
    spacing_mm : float
        Voxel edge [mm].
    shading : ShadingParams, optional
        Default: the shipped ``bonesim/data/shading.toml``.

    Returns
    -------
    int
        Whole bricks (``BRICK`` voxels each), at least 1.
    """
    params = load_shading() if shading is None else shading
    reach = max(tint_reach(params, spacing_mm), 2 * NORMAL_RADIUS) + 1
    return max(1, int(math.ceil(reach / BRICK)))


class BodySurfaces:
    """Each living body's own grid and surface (see the module docstring).

    Make one with :meth:`build` (from scratch) or :meth:`take_over` (at the
    first split, from the one-body surface), then call :meth:`update` after
    every batch of events.

    Parameters
    ----------
    model : Model
        Colours, bone labels and spacing.

    Attributes
    ----------
    grids : dict of int -> Grid
        Body id -> the grid of only that body's voxels, body frame (= grid
        coordinates of the replica).
    surfaces : dict of int -> Surface
        Body id -> its surface, body frame [mm].
    revision : dict of int -> int
        Body id -> a number that grows whenever that body's surface changes
        (built or updated); lets a viewer skip bodies it drew already.
    margin : int
        Bricks around a fragment's bounds (:func:`margin_bricks`).
    """

    def __init__(self, model):
        self.model = model
        self.grids: dict[int, Grid] = {}
        self.surfaces: dict[int, Surface] = {}
        self.revision: dict[int, int] = {}
        self._count = 0
        self.margin = margin_bricks(model.grid.spacing_mm)

    def _bump(self, b: int) -> None:
        self._count += 1
        self.revision[b] = self._count

    # ---------------------------------------------------------------- build
    @classmethod
    def build(cls, model, state) -> "BodySurfaces":
        """Every living body of ``state`` tessellated from scratch.

        Parameters
        ----------
        model : Model
        state : State
            The replica's tissue (``grid``, ``body``, ``alive``, ``bounds``).
        """
        out = cls(model)
        for b in np.flatnonzero(state.alive):
            out._build_body(state, int(b))
        return out

    @classmethod
    def take_over(cls, model, state, main: Surface, changed, touched) -> "BodySurfaces":
        """The first split: body 0 keeps the one-body surface ``main``.

        Parameters
        ----------
        model : Model
        state : State
            The replica's tissue after the batch.
        main : Surface
            The surface of the whole replica grid as of the previous batch;
            updated in place to show only body 0.
        changed : (n, 3) int
            Every voxel whose density in body 0's grid can differ from what
            ``main`` was last updated with: the batch's removed voxels and
            the voxels its splits moved.
        touched : (m, 3) int
            The batch's shading hints.
        """
        out = cls(model)
        g = state.grid
        g0 = Grid(g.spacing_mm, g.origin_mm, g.shape, g.keys, g.vals, g.bricks,
                  masked_density(state, 0), g.label.copy())
        main.update(g0, _ijk(changed), _ijk(touched))
        out.grids[0], out.surfaces[0] = g0, main
        out._bump(0)
        for b in np.flatnonzero(state.alive):
            if b != 0:
                out._build_body(state, int(b))
        return out

    def _build_body(self, state, b: int) -> None:
        g = state.grid
        if b == 0:
            grid = Grid(g.spacing_mm, g.origin_mm, g.shape, g.keys, g.vals, g.bricks,
                        masked_density(state, 0), g.label.copy())
        else:
            bd = state.bounds[b].astype(np.int64)
            lo = (bd[:3] >> BRICK_SHIFT) - self.margin
            hi = (bd[3:] >> BRICK_SHIFT) + self.margin
            sel = np.all((g.bricks >= lo) & (g.bricks <= hi), axis=1)
            grid = g.sub_grid(lo, hi)                 # the same bricks, in order
            grid.density[:] = masked_density(state, b, sel)
        self.grids[b] = grid
        self.surfaces[b] = Surface.of_model(self.model, grid)
        self._bump(b)

    # --------------------------------------------------------------- update
    def update(self, state, removed, touched, split_ijk, split_src, built) -> dict:
        """Bring every body's grid and surface in step with one batch.

        Parameters
        ----------
        state : State
            The replica's tissue after the batch.
        removed : (n, 3) int
            Voxels the batch removed (any body).
        touched : (m, 3) int
            Voxels whose density was lowered (shading hints; any body).
        split_ijk : (s, 3) int
            Voxels the batch's splits moved, in order.
        split_src : (s,) int
            The body each of them left.
        built : iterable of int
            Bodies the batch created or grew: tessellated again from scratch.

        Returns
        -------
        dict
            Body id -> ``Surface.update`` statistics of the bodies updated
            incrementally (``"built"`` for the others).
        """
        g = state.grid
        removed, touched, split_ijk = _ijk(removed), _ijk(touched), _ijk(split_ijk)
        split_src = np.asarray(split_src, dtype=np.int64).reshape(-1)
        built = set(int(b) for b in built)
        rid = voxel_bodies(g, state.body, removed, none=BODY_LIMIT)
        tid = voxel_bodies(g, state.body, touched, none=BODY_LIMIT)
        out = {}
        for b in list(self.surfaces):
            if b in built:
                continue
            if not state.alive[b]:
                del self.surfaces[b], self.grids[b], self.revision[b]
                continue
            rem = removed[rid == b]
            if (split_src == b).any():
                rem = np.concatenate((rem, split_ijk[split_src == b]))
            tch = touched[tid == b]
            if not (len(rem) or len(tch)):
                continue
            bg = self.grids[b]
            for ijk in (rem, tch):
                if len(ijk):
                    _sync_body(g.keys, g.vals, g.density, state.body, np.uint8(b), bg.keys,
                               bg.vals, bg.density, ijk)
            out[b] = self.surfaces[b].update(bg, rem, tch)
            self._bump(b)
        for b in np.flatnonzero(state.alive):
            b = int(b)
            if b in built or b not in self.surfaces:
                self._build_body(state, b)
                out[b] = "built"
        return out
