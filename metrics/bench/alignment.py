"""Benchmark of the force-trajectory alignment (:mod:`metrics.alignment`).

``dp_align_1000_ms``
    :func:`metrics.alignment.dp_align` on two 1000-sample curves (the
    thesis' 10 s trial at 100 Hz; a 1000 x 1000 table, no band), median of
    several runs [ms], the kernel compiled first. Beside it: the whole
    :func:`metrics.alignment.align` of two irregular 10 s recordings at about
    1 kHz (resampling, box filter, DP, warp), and a pure-Python DP (the same
    recurrence, cost only) on a :data:`NAIVE_N`-square table for scale,
    compared per cell.

``bonesim bench`` finds it by name (:data:`bonesim.bench.suite.BENCHMARKS`).
Figures are wall-clock on whatever machine runs them.
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ["DP_N", "NAIVE_N", "bench_dp_align"]

#: Samples per curve of the timed DP.
DP_N = 1000
#: Samples per curve of the pure-Python reference.
NAIVE_N = 200


def _naive_cost(fa, fb, sa, sb, w_force, w_slope, penalty) -> float:
    """The DP's recurrence in plain Python over two rows (cost only)."""
    n, m = len(fa), len(fb)
    inf = float("inf")
    prev = [inf] * m
    for i in range(n):
        cur = [inf] * m
        for j in range(m):
            df, ds = fa[i] - fb[j], sa[i] - sb[j]
            c = w_force * (df * df) + w_slope * (ds * ds)
            if i == 0 and j == 0:
                cur[j] = c
                continue
            best = inf
            if i > 0 and j > 0:
                best = prev[j - 1]
            if i > 0 and prev[j] + penalty < best:
                best = prev[j] + penalty
            if j > 0 and cur[j - 1] + penalty < best:
                best = cur[j - 1] + penalty
            cur[j] = c + best
        prev = cur
    return prev[m - 1]


def _curve(rng, n: int, rate_hz: float) -> np.ndarray:
    """A bounded random-walk force [N] of ``n`` samples (0 to 3.3 N)."""
    return np.clip(np.cumsum(rng.normal(0.0, 3.0 / np.sqrt(rate_hz), n)) + 1.5, 0.0, 3.3)


def bench_dp_align(quick: bool = False) -> dict:
    """DP alignment of 1000 x 1000 samples, the full alignment, and a naive
    reference."""
    from metrics.alignment import (DEFAULT_PENALTY, DEFAULT_RATE_HZ, DEFAULT_W_FORCE,
                                   DEFAULT_W_SLOPE, align, dp_align, slope)

    rng = np.random.default_rng(0)
    fa, fb = _curve(rng, DP_N, DEFAULT_RATE_HZ), _curve(rng, DP_N, DEFAULT_RATE_HZ)
    sa, sb = slope(fa, DEFAULT_RATE_HZ), slope(fb, DEFAULT_RATE_HZ)
    dp_align(fa[:10], fb[:10], sa[:10], sb[:10])          # compile (cached on disk)
    reps = 3 if quick else 9
    dp = []
    for _ in range(reps):
        t0 = time.perf_counter()
        cost, path = dp_align(fa, fb, sa, sb)
        dp.append(time.perf_counter() - t0)
    # the whole alignment of two irregular ~1 kHz, 10 s recordings
    raw_t = [np.cumsum(rng.uniform(0.0008, 0.0012, 10000)) for _ in range(2)]
    raw_f = [_curve(rng, 10000, 1000.0) for _ in range(2)]
    full = []
    for _ in range(reps):
        t0 = time.perf_counter()
        al = align(raw_t[0], raw_f[0], raw_t[1], raw_f[1])
        full.append(time.perf_counter() - t0)
    k = NAIVE_N
    args = [a[:k].tolist() for a in (fa, fb, sa, sb)]
    t0 = time.perf_counter()
    naive = _naive_cost(*args, DEFAULT_W_FORCE, DEFAULT_W_SLOPE, DEFAULT_PENALTY)
    t_naive = time.perf_counter() - t0
    small = dp_align(fa[:k], fb[:k], sa[:k], sb[:k])[0]
    ms = float(np.median(dp)) * 1e3
    naive_ns_cell = t_naive * 1e9 / (k * k)
    ns_cell = ms * 1e6 / (DP_N * DP_N)
    return {"dp_align_1000_ms": {
        "value": round(ms, 3), "unit": "ms", "runs": reps, "cells": DP_N * DP_N,
        "ns_per_cell": round(ns_cell, 2), "path_length": int(len(path)),
        "min_ms": round(float(np.min(dp)) * 1e3, 3),
        "align_10s_1khz_ms": round(float(np.median(full)) * 1e3, 3),
        "align_table": [len(al.t_s), len(al.applied_n)],
        "naive_python": {"n": k, "ms": round(t_naive * 1e3, 1),
                         "ns_per_cell": round(naive_ns_cell, 1),
                         "same_cost": bool(naive == small)},
        "speedup_per_cell_vs_naive": round(naive_ns_cell / ns_cell, 1),
        "what": "metrics.alignment.dp_align, 1000 x 1000 table (no band), default weights; "
                "median of runs after compiling; align_10s_1khz_ms is the whole align() of "
                "two irregular 10 s ~1 kHz recordings; the naive reference is the same "
                "recurrence in pure Python on a smaller table"}}
