"""Benchmark helpers (bonesim.bench.tools) against naive references, and the
haptic step's figures against its floor."""
from __future__ import annotations

import numpy as np

from bonesim.bench.tools import ball_offsets, stencil_density_pass
from bonesim.io.loading import load_model


def test_stencil_density_pass_matches_a_naive_lookup():
    model = load_model("phantom", "cutting-7mm")
    grid, samples = model.grid, model.stencil.packed
    rng = np.random.default_rng(2)
    lo = grid.origin_mm
    hi = grid.origin_mm + grid.spacing_mm * np.asarray(grid.shape)
    for pos in np.vstack([rng.uniform(lo - 3.0, hi + 3.0, (12, 3)),   # some outside
                          model.grid.origin_mm + 26.0 + rng.normal(0, 5, (12, 3))]):
        want = 0.0
        for o in samples[:, :3].astype(np.float64):
            ijk = np.floor((pos + o - grid.origin_mm) / grid.spacing_mm + 0.5).astype(int)
            want += float(grid.density_at(*ijk))
        got = stencil_density_pass(grid, samples, pos, model.burr.radius_mm)
        assert abs(got - want) < 1e-6 * len(samples)


def test_ball_offsets_are_the_voxels_inside():
    b = ball_offsets(2.5)
    assert len(b) == len({tuple(v) for v in b.tolist()})
    g = np.stack(np.meshgrid(*[np.arange(-3, 4)] * 3, indexing="ij"), -1).reshape(-1, 3)
    inside = {tuple(v) for v in g[(g ** 2).sum(1) <= 6.25].tolist()}
    assert {tuple(v) for v in b.tolist()} == inside


def test_haptic_bench_reports_its_floor():
    from bonesim.bench.suite import BENCHMARKS

    out = BENCHMARKS["haptic_step_vs_floor"](quick=True)
    p50, floor = out["haptic_step_7mm_p50_us"]["value"], out["haptic_step_floor_us"]["value"]
    assert floor > 0 and p50 > 0         # how much more the step costs is the figure's
    assert abs(out["haptic_step_vs_floor"]["value"] - p50 / floor) <= 0.05 * p50 / floor
    four = out["haptic_step_7mm_4x_p99_us"]
    # at 4x on 0.5 mm voxels the fixed budget binds: the 2x lattice's samples
    assert four["oversample"] == 4 and four["samples"] == out["haptic_step_floor_us"]["samples"]
    assert four["value"] >= four["p50_us"] > 0
    ratio = out["haptic_step_4x_vs_2x_p50"]["value"]
    assert abs(ratio - four["p50_us"] / p50) <= 0.05 * ratio
