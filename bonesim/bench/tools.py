"""Small helpers the benchmarks share: a ball of voxel offsets, emptying
voxels as a burr would (the surface and window benchmarks, the soak test),
and the haptic step's floor."""
from __future__ import annotations

import numpy as np
from numba import njit

from bonesim.engine.grid import BRICK_SHIFT, voxel_offset
from bonesim.engine.haptics import block_bricks, block_size

__all__ = ["ball_offsets", "remove_voxels", "stencil_density_pass", "floor_scratch"]


@njit(cache=True, nogil=True)
def _density_pass(keys, vals, density, origin, spacing, samples, pos, radius, lbrick,
                  ldens):
    # the local block around the burr, gathered as the haptic step gathers it
    n_vox = int(round(len(ldens) ** (1.0 / 3.0)))
    lo0, lo1, lo2, _ = block_bricks(keys, vals, pos, radius, origin, spacing, lbrick)
    b0, b1, b2 = lo0 >> BRICK_SHIFT, lo1 >> BRICK_SHIFT, lo2 >> BRICK_SHIFT
    nn = n_vox * n_vox
    for x in range(n_vox):
        i = lo0 + x
        bx = (i >> BRICK_SHIFT) - b0
        for y in range(n_vox):
            j = lo1 + y
            by = (j >> BRICK_SHIFT) - b1
            base = x * nn + y * n_vox
            for z in range(n_vox):
                k = lo2 + z
                b = lbrick[bx, by, (k >> BRICK_SHIFT) - b2]
                ldens[base + z] = density[b, voxel_offset(i, j, k)] if b >= 0 else 0.0
    # one lookup per sample
    inv = 1.0 / spacing
    c0 = (pos[0] - origin[0]) * inv + 0.5 - lo0
    c1 = (pos[1] - origin[1]) * inv + 0.5 - lo1
    c2 = (pos[2] - origin[2]) * inv + 0.5 - lo2
    total = 0.0
    for q in range(samples.shape[0]):
        li = (int(c0 + samples[q, 0] * inv) * n_vox
              + int(c1 + samples[q, 1] * inv)) * n_vox + int(c2 + samples[q, 2] * inv)
        total += ldens[li]
    return total


def stencil_density_pass(grid, samples, pos_mm, radius_mm: float, scratch=None) -> float:
    """The haptic step's floor: one pass over a burr stencil's samples that
    only looks up each sample's voxel density.

    It gathers the burr's neighbourhood into a dense block as the haptic step
    does (:func:`bonesim.engine.haptics.haptic_kernel`), then reads one density per
    sample (offsets along the case axes): no tool frame, force, removal or
    events.

    Parameters
    ----------
    grid : bonesim.engine.grid.Grid
    samples : (n, >=3) float32
        Sample offsets from the burr's centre [mm] (the stencil's packed rows).
    pos_mm : (3,) float64
        Burr centre, case frame [mm].
    radius_mm : float
        Burr radius [mm] (sizes the block).
    scratch : tuple, optional
        ``(lbrick, ldens)`` from :func:`floor_scratch` (made if not given).

    Returns
    -------
    float
        The sum of the densities looked up.
    """
    samples = np.asarray(samples)
    if samples.ndim != 2 or samples.shape[1] < 3:
        raise ValueError(f"samples must be (n, >=3), got {samples.shape}")
    lbrick, ldens = scratch if scratch is not None else floor_scratch(radius_mm,
                                                                      grid.spacing_mm)
    return _density_pass(grid.keys, grid.vals, grid.density_ro,
                         np.asarray(grid.origin_mm, np.float64), float(grid.spacing_mm),
                         samples, np.asarray(pos_mm, np.float64), float(radius_mm),
                         lbrick, ldens)


def floor_scratch(radius_mm: float, spacing_mm: float) -> tuple:
    """Scratch arrays for :func:`stencil_density_pass` (the haptic step's sizes)."""
    n_vox, n_brick = block_size(radius_mm, spacing_mm)
    return (np.empty((n_brick,) * 3, np.int32), np.empty(n_vox ** 3, np.float32))


def ball_offsets(radius_vox: float) -> np.ndarray:
    """Integer offsets (n, 3) int32 of the voxels of a ball of ``radius_vox`` [voxels]."""
    m = int(np.ceil(radius_vox))
    g = np.stack(np.meshgrid(*[np.arange(-m, m + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return g[(g ** 2).sum(1) <= radius_vox ** 2].astype(np.int32)


def remove_voxels(grid, ijk) -> np.ndarray:
    """Empty the occupied voxels among ``ijk`` (as a burr would); returns them
    as (n, 3) int32, the list a surface update needs."""
    from bonesim.engine.grid import BRICK_SHIFT, find_brick, voxel_offset

    out = []
    for i, j, k in ijk:
        b = find_brick(grid.keys, grid.vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                       k >> BRICK_SHIFT)
        if b >= 0:
            o = voxel_offset(i, j, k)
            if grid.density[b, o] > 0:
                grid.density[b, o] = 0.0
                out.append((i, j, k))
    return np.array(out, dtype=np.int32).reshape(-1, 3)
