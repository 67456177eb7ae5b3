"""The bench's registry: benchmarks outside the suite are found by dotted
name (the research metrics' among them, without bonesim importing metrics)."""
from __future__ import annotations

import pytest

from bonesim.bench.suite import BENCHMARKS, ByName
from bonesim.errors import BonesimError


def test_the_metrics_benchmarks_are_named_not_imported():
    named = {v.ref for v in BENCHMARKS.values() if isinstance(v, ByName)}
    assert {"metrics.bench.alignment:bench_dp_align",
            "metrics.bench.cohort:bench_metrics_cohort"} <= named
    fn = BENCHMARKS["dp_align_1000_ms"]
    assert fn.__name__ == "bench_dp_align" and fn.resolve().__module__ == "metrics.bench.alignment"
    # figures one run gives share one entry (run_benchmarks runs it once)
    assert BENCHMARKS["cohort_sessions_per_s"] is BENCHMARKS["metrics_run_s"]


def test_a_benchmark_that_cannot_be_found_is_one_line():
    with pytest.raises(BonesimError) as e:
        ByName("metrics.bench.no_such_module:bench_x").resolve()
    assert "\n" not in str(e.value) and "metrics.bench.no_such_module:bench_x" in str(e.value)
    with pytest.raises(ValueError, match="module:function"):
        ByName("metrics.bench.alignment")
