"""The alignment benchmark (metrics.bench.alignment): registered,
reports its figures, and its pure-Python reference agrees with the kernel."""
from __future__ import annotations

import numpy as np

from metrics.bench.alignment import _naive_cost


def test_the_bench_reports_the_1000_square_dp():
    from bonesim.bench.suite import BENCHMARKS

    out = BENCHMARKS["dp_align_1000_ms"](quick=True)["dp_align_1000_ms"]
    assert out["unit"] == "ms" and out["value"] >= out["min_ms"] > 0
    assert out["cells"] == 1000 * 1000 and out["align_table"][0] == 1000
    assert out["naive_python"]["same_cost"]


def test_the_naive_cost_is_the_kernels():
    from metrics.alignment import dp_align

    rng = np.random.default_rng(1)
    fa, fb, sa, sb = (rng.integers(0, 3, k).astype(float) for k in (17, 23, 17, 23))
    want = dp_align(fa, fb, sa, sb, w_force=1.0, w_slope=0.5, penalty=0.25)[0]
    assert _naive_cost(*(a.tolist() for a in (fa, fb, sa, sb)), 1.0, 0.5, 0.25) == want
