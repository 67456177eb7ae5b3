"""Soak: many cumulative burr-ball removals on the phantom keep the
incremental surface identical to a from-scratch tessellation (both update
paths: the dense-window path and the hash-set fallback)."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.grid import BRICK_SHIFT, find_brick, voxel_offset
from bonesim.model import load_model
from bonesim.surface import Surface

pytestmark = pytest.mark.slow


def _ball(r):
    m = int(np.ceil(r))
    g = np.stack(np.meshgrid(*[np.arange(-m, m + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return g[(g ** 2).sum(1) <= r * r].astype(np.int32)


@pytest.mark.parametrize("window", [True, False])
def test_cumulative_balls_match_rebuild(window):
    model = load_model("phantom", "cutting-5mm")
    grid = model.grid.copy()
    surf = Surface.build(grid, model.colors)
    if not window:
        surf._win_per_input = 0                   # force the hash-set path
    rng = np.random.default_rng(11)
    ball = _ball(7.8)
    done = 0
    while done < 40:
        pos = surf.arrays()[0]
        ijk_v = np.floor((pos - grid.origin_mm) / grid.spacing_mm + 0.5).astype(np.int32)
        c = ijk_v[rng.integers(len(ijk_v))]
        ijk = c + ball
        dens, _ = grid.to_dense(lo=c - 9, shape=(19, 19, 19))
        ijk = np.ascontiguousarray(ijk[dens[tuple((ijk - (c - 9)).T)] > 0])
        if len(ijk) < 600:
            continue
        for i, j, k in ijk:
            b = find_brick(grid.keys, grid.vals, i >> BRICK_SHIFT, j >> BRICK_SHIFT,
                           k >> BRICK_SHIFT)
            grid.density[b, voxel_offset(i, j, k)] = 0.0
        surf.update(grid, ijk)
        done += 1
        if done % 10 == 0:
            fresh = Surface.build(grid, model.colors)
            assert not fresh.canonical().differences(surf.canonical()), f"after {done} balls"
