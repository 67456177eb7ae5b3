"""The bone's bodies as :class:`bonesim.physics.dust.DustGrid` sees them.

The dust lattice is the case frame; a body's voxels stay where they were cut,
in the body's own frame (:mod:`bonesim.engine.bodies`). These helpers put a
moved body's removals on the lattice and tell the step kernels which bone is
a wall (see "Bodies" in :mod:`bonesim.physics.dust.grid`).
"""
from __future__ import annotations

import numpy as np

from bonesim.engine.bodies import all_identity, is_identity
from bonesim.engine.grid import BRICK_VOXELS

__all__ = ["case_cells", "wall_arrays"]

# the step's wall arguments when every bone cell is a wall (never read)
_NO_BODY = np.zeros((1, BRICK_VOXELS), np.uint8)
_ALL_WALLS = np.zeros(0, np.uint8)


def case_cells(ijk, amount, body, bodies, origin_mm, spacing_mm, bounds=None):
    """Removed voxels of bodies ``body`` as cells of the case-frame lattice.

    Parameters
    ----------
    ijk : (n, 3) int64
        Removed voxels, each in its body's frame.
    amount : (n,) float
        Dust per voxel [cells]; kept alongside the cells.
    body : (n,) int
        The body of each voxel.
    bodies : Bodies or State
        ``pose``, ``pose_m`` and ``alive`` are read.
    origin_mm : (3,) float64
        Centre of cell (0, 0, 0) [mm] (the bone grid's, in every body's frame).
    spacing_mm : float
        Cell edge [mm].
    bounds : (6,) int, optional
        Domain ``lo, hi`` [cells]; cells outside it are dropped.

    Returns
    -------
    ijk : (m, 3) int64
        For a body at the identity the voxel itself, else the cell nearest
        to its centre's case-frame position ``R c + t``.
    amount : (m,) float64
    """
    body = np.broadcast_to(np.asarray(body, dtype=np.int64), (len(ijk),))
    if len(body) and (body.min() < 0 or body.max() >= len(bodies.alive)):
        raise ValueError(f"removal bodies must lie in 0..{len(bodies.alive) - 1}")
    out = np.array(ijk, dtype=np.int64)
    h, o = float(spacing_mm), np.asarray(origin_mm, dtype=np.float64)
    for b in np.unique(body):
        if is_identity(bodies.pose[b]):
            continue
        sel = body == b
        m = np.asarray(bodies.pose_m[b], dtype=np.float64)
        c = (o + h * out[sel]) @ m[:, :3].T + m[:, 3]        # case frame [mm]
        out[sel] = np.floor((c - o) / h + 0.5).astype(np.int64)
    amount = np.asarray(amount, dtype=np.float64)
    if bounds is None:
        return out, amount
    keep = ((out >= bounds[:3]) & (out < bounds[3:])).all(axis=1)
    return np.ascontiguousarray(out[keep]), np.ascontiguousarray(amount[keep])


def wall_arrays(bone_grid, bodies):
    """``(bone_body, wall_body)`` for the dust step's kernels.

    Returns
    -------
    bone_body : (n_bricks, 512) uint8
        The body of each bone voxel (``bodies.body``).
    wall_body : (max_bodies,) uint8
        1 for the living bodies at the identity pose: their bone is a wall.
        Empty (and ``bone_body`` a placeholder, never read) when there is no
        bone grid or every body sits at the identity: all bone is a wall,
        exactly as without bodies.
    """
    if bone_grid is None or all_identity(bodies):
        return _NO_BODY, _ALL_WALLS
    body = bodies.body
    if body.shape != bone_grid.density.shape:
        raise ValueError(f"bodies.body has shape {body.shape}, the bone grid's density "
                         f"{bone_grid.density.shape}")
    wall = np.zeros(len(bodies.alive), np.uint8)
    for b in np.flatnonzero(bodies.alive):
        wall[b] = is_identity(bodies.pose[b])
    return body, wall
