"""The world-step benchmark (bonesim.bench.world) runs and reports both figures."""
from __future__ import annotations

import pytest

from bonesim.bench.suite import BENCHMARKS
from bonesim.bench.world import bench_world_step


def test_world_step_figures_are_registered_and_reported():
    assert {"world_step_vs_step_p50", "world_step_7mm_p99_us"} <= set(BENCHMARKS)
    out = bench_world_step(quick=True)
    r = out["world_step_vs_step_p50"]
    assert r["unit"] == "x" and r["steps"] == 2000
    assert r["world_p50_us"] > 0 and r["step_p50_us"] > 0
    assert r["value"] == pytest.approx(r["world_p50_us"] / r["step_p50_us"], rel=0.02)
    assert out["world_step_7mm_p99_us"]["value"] >= r["world_p50_us"]
