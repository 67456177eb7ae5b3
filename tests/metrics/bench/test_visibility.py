"""The offline visibility benchmark (metrics.bench.visibility): registered,
and its figures describe the run it recomputed (no timing is asserted)."""
from __future__ import annotations


def test_visibility_offline_figures_registered():
    from bonesim.bench.suite import BENCHMARKS

    out = BENCHMARKS["visibility_offline_removals_per_s"](quick=True)
    v = out["visibility_offline_removals_per_s"]
    assert v["unit"] == "removals/s" and v["value"] > 0
    assert v["removals"] > 1000 and v["run_s"] > 30
    assert v["equals_live"] is True
    assert 0.0 < v["visible_fraction"] <= 1.0
