"""Benchmark of the offline voxel-visibility metric (:mod:`metrics.visibility`).

``visibility_offline_removals_per_s``
    Removals judged per second when a recorded run's visibility is
    recomputed from the file (:func:`metrics.visibility.recompute_visible`):
    the phantom demo with the default burr (``cutting-5mm``) recorded by
    ``bonesim simulate --record`` (the whole demo, about four minutes of
    drilling and 30,000 removals; the first minute with ``quick``). The
    session is read and its models rebuilt before the timing; the figure
    is the median of three recomputations. The detail gives the model
    rebuild and file read times, and whether the recomputed verdicts equal
    the recorder's live ones.
"""
from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

__all__ = ["bench_metrics_visibility"]


def bench_metrics_visibility(quick=False) -> dict:
    from bonesim.engine import events
    from bonesim.io.case import load_case
    from bonesim.io.loading import load_model
    from bonesim.io.toolpath import demo_trajectory
    from bonesim.runtime.simulate import run_trajectory
    from bonesim.session.reader import read_session
    from metrics.visibility import recompute_visible

    model = load_model("phantom", "cutting-5mm")
    t = demo_trajectory(load_case("phantom"), "cutting-5mm")
    start = int(np.flatnonzero(t.drill)[0])
    stop = len(t.t_s)
    if quick:
        stop = min(stop, int(np.searchsorted(t.t_s, t.t_s[start] + 60.0)))
    traj = t.at_times(t.t_s[start:stop])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "run.h5"
        run_trajectory(model, traj, surface=False, record=path)
        t0 = time.perf_counter()
        session = read_session(path)
        read_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    models = session.burr_models()
    models_s = time.perf_counter() - t0
    n = int(np.sum(session.tissue["kind"] == events.REMOVED))
    recompute_visible(session, models)             # kernels loaded, outside the timing
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        vis = recompute_visible(session, models)
        times.append(time.perf_counter() - t0)
    dt = float(np.median(times))
    rem = session.tissue["kind"] == events.REMOVED
    return {"visibility_offline_removals_per_s": {
        "value": round(n / dt) if dt > 0 else 0, "unit": "removals/s",
        "removals": n, "run_s": round(session.duration_s, 1),
        "recompute_s": round(dt, 4), "read_session_s": round(read_s, 3),
        "burr_models_s": round(models_s, 3),
        "visible_fraction": round(float(np.mean(vis[rem] == 1)), 4) if n else None,
        "equals_live": bool(np.array_equal(vis, session.tissue["visible"]))}}
