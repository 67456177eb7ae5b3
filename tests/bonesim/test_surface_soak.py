"""Soak: many cumulative burr-ball removals on the phantom keep the
incremental surface identical to a from-scratch tessellation, normals and
thin-bone tint included (both update paths: the dense-window path and the
hash-set fallback)."""
from __future__ import annotations

import numpy as np
import pytest

from bonesim.bench_tools import ball_offsets, remove_voxels
from bonesim.loading import load_model
from bonesim.surface import Surface

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("window", [True, False])
def test_cumulative_balls_match_rebuild(window):
    model = load_model("phantom", "cutting-5mm")
    grid = model.grid.copy()
    surf = Surface.of_model(model, grid)
    if not window:
        surf._win_per_input = 0                   # force the hash-set path
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
