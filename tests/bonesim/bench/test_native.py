"""The native-resolution bench's floor (bonesim.bench.native) against a naive
lookup, and its figures registered in the suite's table."""
from __future__ import annotations

import numpy as np

from bonesim.bench.native import budget_floor_pass
from bonesim.bench.suite import BENCHMARKS, ByName
from bonesim.engine.model import make_state

from tests.bonesim.fakes import FakeBurr, block_model


def test_budget_floor_pass_matches_a_naive_lookup():
    model, _ = block_model(shape=(60, 60, 60), fill_z=35, spacing=0.1,
                           burr=FakeBurr(radius_mm=1.2))
    assert model.budget.binding
    grid, samples = model.grid, model.stencil.packed
    lbrick = make_state(model)._lbrick
    rng = np.random.default_rng(4)
    for pos in rng.uniform(-1.0, 7.0, (16, 3)):
        want = 0.0
        for o in samples[:, :3].astype(np.float64):
            ijk = np.floor((pos + o - grid.origin_mm) / grid.spacing_mm + 0.5).astype(int)
            want += float(grid.density_at(*ijk))
        got = budget_floor_pass(grid, samples, pos, 1.2, lbrick)
        assert abs(got - want) < 1e-6 * len(samples)


def test_the_native_figures_are_in_the_table():
    names = [f"haptic_step_native_{v}_{f}" for v in ("019", "010")
             for f in ("p99_us", "vs_05", "vs_floor")]
    refs = {BENCHMARKS[n].ref for n in names}
    assert refs == {"bonesim.bench.native:bench_native_step"}
    assert all(isinstance(BENCHMARKS[n], ByName) for n in names)
