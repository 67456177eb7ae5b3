"""Small helpers the benchmarks share: a ball of voxel offsets, and emptying
voxels as a burr would (the surface and window benchmarks, the soak test)."""
from __future__ import annotations

import numpy as np

__all__ = ["ball_offsets", "remove_voxels"]


def ball_offsets(radius_vox: float) -> np.ndarray:
    """Integer offsets (n, 3) int32 of the voxels of a ball of ``radius_vox`` [voxels]."""
    m = int(np.ceil(radius_vox))
    g = np.stack(np.meshgrid(*[np.arange(-m, m + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return g[(g ** 2).sum(1) <= radius_vox ** 2].astype(np.int32)


def remove_voxels(grid, ijk) -> np.ndarray:
    """Empty the occupied voxels among ``ijk`` (as a burr would); returns them
    as (n, 3) int32, the list a surface update needs."""
    from .grid import BRICK_SHIFT, find_brick, voxel_offset

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
