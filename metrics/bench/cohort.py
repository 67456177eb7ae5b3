"""Benchmarks of the cohort scorer (:mod:`metrics.cohort`) and of one run's metrics.

``cohort_sessions_per_s``
    Session files scored per second by :func:`metrics.cohort.score_cohort`
    on a synthetic cohort (:func:`metrics.synth.synth_cohort`, 8 expert-like
    and 8 novice-like participants with 3 sessions each: 48 runs of 6 s;
    2 + 2 participants with 2 sessions of 4 s with ``quick``), recorded once
    in a temporary folder before the timing. Scored on a
    ``LocalCluster`` with 1 worker and with 2 worker processes, passed by
    address: a first pass warms the workers (each rebuilds the case's models
    once and loads the numba kernels), the second, timed, gives the figure:
    the whole :func:`~metrics.cohort.score_cohort` call, its central steps
    (Naive Bayes, final product, exceedances, statistics, serial in the
    client) included. The value is the 2-worker figure; the detail gives
    both, ``scaling_1_to_2`` (2-worker over 1-worker throughput; at most 2,
    less with the serial central part or busy cores) and each first pass's
    wall time from starting the cluster [s], as a user of ``bonesim metrics
    cohort`` sees it, and ``central_s``, the serial central part [s].
``cohort_stats_s``
    Seconds of the statistics step of that timed 2-worker pass
    (:func:`metrics.group_stats.group_statistics` over every metric with the
    mixed models and corrections, the Naive Bayes ROC and the test-retest
    agreement), ``meta["stats_s"]``.
``metrics_run_s``
    Seconds of :func:`metrics.run.run_metrics` on one 3-minute synthetic
    expert-like run (1 minute with ``quick``), warm: the second call (the
    first loads the numba kernels); the session is read from the file each
    call.
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

__all__ = ["bench_metrics_cohort"]


def _cohort(tmp: Path, quick: bool) -> dict:
    from metrics.cohort import local_cluster, score_cohort
    from metrics.synth import BEHAVIOURS_FILE, PARTICIPANTS_CSV, synth_cohort

    n, k, dur = (2, 2, 4.0) if quick else (8, 3, 6.0)
    d = tmp / "cohort"
    t0 = time.perf_counter()
    paths = synth_cohort(d, n, n, seed=0, duration_s=dur, sessions=k,
                         behaviours=BEHAVIOURS_FILE)
    record_s = time.perf_counter() - t0
    rates, cold, central, stats_s = {}, {}, {}, {}
    for w in (1, 2):
        t0 = time.perf_counter()
        with local_cluster(w) as cluster:
            score_cohort(d, d / PARTICIPANTS_CSV, scheduler=cluster.scheduler_address)
            cold[w] = time.perf_counter() - t0
            t0 = time.perf_counter()
            res = score_cohort(d, d / PARTICIPANTS_CSV, scheduler=cluster.scheduler_address)
            warm = time.perf_counter() - t0
        central[w] = res.meta["central_s"]
        stats_s[w] = res.meta["stats_s"]
        rates[w] = len(paths) / warm
        failed = int((res.table["error"] != "").sum())
    return {"cohort_sessions_per_s": {
        "value": round(rates[2], 3), "unit": "sessions/s",
        "sessions": len(paths), "participants": 2 * n, "sessions_each": k, "run_s": dur,
        "sessions_per_s_1_worker": round(rates[1], 3),
        "sessions_per_s_2_workers": round(rates[2], 3),
        "scaling_1_to_2": round(rates[2] / rates[1], 3),
        "first_pass_s_1_worker": round(cold[1], 2),
        "first_pass_s_2_workers": round(cold[2], 2),
        "central_s": round(central[2], 3),
        "failed": failed, "record_s": round(record_s, 1)},
        "cohort_stats_s": {"value": round(stats_s[2], 3), "unit": "s",
                           "sessions": len(paths), "metrics": int(len(res.stats))}}


def _run(tmp: Path, quick: bool) -> dict:
    from metrics.run import run_metrics
    from metrics.synth import synth_cohort

    dur = 60.0 if quick else 180.0
    (path,) = synth_cohort(tmp / "one", 1, 0, seed=1, duration_s=dur)
    t0 = time.perf_counter()
    run_metrics(path)
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = run_metrics(path)
    warm = time.perf_counter() - t0
    return {"metrics_run_s": {
        "value": round(warm, 3), "unit": "s", "run_s": dur,
        "removed_voxels": out["run"]["removed_voxels"], "first_call_s": round(cold, 3)}}


def bench_metrics_cohort(quick=False) -> dict:
    """Both figures of the module docstring."""
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        return {**_cohort(tmp, quick), **_run(tmp, quick)}
