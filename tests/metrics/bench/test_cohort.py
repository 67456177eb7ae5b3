"""The cohort benchmarks (metrics.bench.cohort): registered as one entry
point, and their figures describe what they scored (no timing is asserted)."""
from __future__ import annotations


def test_cohort_figures_registered():
    from bonesim.bench.suite import BENCHMARKS

    assert BENCHMARKS["cohort_sessions_per_s"] is BENCHMARKS["metrics_run_s"] \
        is BENCHMARKS["cohort_stats_s"]
    out = BENCHMARKS["cohort_sessions_per_s"](quick=True)
    c, r = out["cohort_sessions_per_s"], out["metrics_run_s"]
    assert c["unit"] == "sessions/s" and c["value"] > 0 and c["sessions"] == 8
    assert c["participants"] == 4 and c["sessions_each"] == 2
    st = out["cohort_stats_s"]
    assert st["unit"] == "s" and st["value"] > 0 and st["sessions"] == 8 and st["metrics"] > 0
    assert c["failed"] == 0 and c["scaling_1_to_2"] > 0
    assert c["value"] == c["sessions_per_s_2_workers"]
    assert r["unit"] == "s" and r["value"] > 0 and r["run_s"] == 60.0
