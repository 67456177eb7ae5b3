"""Soak: many cumulative burr-ball removals on the phantom keep the
incremental surface identical to a from-scratch tessellation, normals and
thin-bone tint included (one window per ball, and every ball tiled into
windows of 4 voxels)."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.bench.tools import ball_offsets, remove_voxels
from bonesim.io.loading import load_model
from bonesim.engine.surface import Surface
from tests.bonesim.fakes import force_tiles

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("tiled", [False, True])
def test_cumulative_balls_match_rebuild(tiled):
    model = load_model("phantom", "cutting-5mm")
    grid = model.grid.copy()
    surf = Surface.of_model(model, grid)
    if tiled:
        force_tiles(surf, 2)                      # tile every update
    rng = np.random.default_rng(11)
    ball = ball_offsets(7.8)
    done = 0
    while done < 40:
        pos = surf.arrays()[0]
        ijk_v = np.floor((pos - grid.origin_mm) / grid.spacing_mm + 0.5).astype(np.int32)
        c = ijk_v[rng.integers(len(ijk_v))]
        ijk = remove_voxels(grid, c + ball)
        surf.update(grid, ijk)
        if len(ijk) < 600:                        # count only balls that cut deep
            continue
        done += 1
        if done % 10 == 0:
            fresh = Surface.of_model(model, grid)
            assert not fresh.canonical().differences(surf.canonical()), f"after {done} balls"
