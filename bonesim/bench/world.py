"""Benchmark: the world step against the haptic step alone, in one run.

The same sweep as ``haptic_step_7mm_p50_us`` (the 7 mm cutting burr half
immersed in a bone block, 2x oversampling, drilling), stepped on two states
with the same samples, alternately: one through
:func:`bonesim.engine.model.step`, the other through
:func:`bonesim.engine.world.world_step` without commands (the rigid set
present, nothing in motion), which is what the haptic loop, ``simulate``
and replay call. The ratio of their p50s, measured interleaved, says what
the world step adds to the step; it does not depend on how loaded the
machine is as much as either time does. Figures are reported, never
asserted.
"""
from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

__all__ = ["bench_world_step"]


def _pct(a, q) -> float:
    return float(np.percentile(np.asarray(a, float), q))


def bench_world_step(quick=False) -> dict:
    """``world_step_vs_step_p50`` and ``world_step_7mm_p99_us``."""
    from bonesim.engine.model import Sample, make_model, make_state, step
    from bonesim.engine.world import world_step
    from bonesim.io.burrs import load_burr
    from bonesim.io.loading import warmup

    warmup()
    n = 2000 if quick else 20000
    burr = load_burr("cutting-7mm")
    labels = np.zeros((120, 120, 60), np.uint8)
    labels[:, :, :40] = 1
    bone = SimpleNamespace(name="bone", kind="bone", display_color=(230, 220, 200))
    model = make_model(labels, 0.5, [bone], burr)
    top = 40 * 0.5 - 0.25
    per_reset = 500
    axis = np.array([0.3, 0.0, -1.0])
    step_ns = np.empty(n, np.int64)
    world_ns = np.empty(n, np.int64)
    perf = time.perf_counter_ns
    a = b = None
    none = ()
    for q in range(n):
        if q % per_reset == 0:
            a, b = make_state(model), make_state(model)     # fresh bone, untimed
        u = q % per_reset
        pos = np.array([10.0 + (0.08 * u) % 40.0, 10.0 + 8.0 * ((q // per_reset) % 5), top])
        smp = Sample(q * 1e-3, pos, axis, True, burr.default_speed_rpm, 1)
        if q % 2:
            t0 = perf()
            step(model, a, smp)
            t1 = perf()
            world_step(model, b, smp, none)
            t2 = perf()
            step_ns[q], world_ns[q] = t1 - t0, t2 - t1
        else:
            t0 = perf()
            world_step(model, b, smp, none)
            t1 = perf()
            step(model, a, smp)
            t2 = perf()
            world_ns[q], step_ns[q] = t1 - t0, t2 - t1
    s_us, w_us = step_ns / 1e3, world_ns / 1e3
    return {
        "world_step_vs_step_p50": {
            "value": round(_pct(w_us, 50) / _pct(s_us, 50), 3), "unit": "x",
            "what": "p50 of the world step without commands / p50 of the haptic step "
                    "alone, the 7 mm sweep of haptic_step_7mm_p50_us, measured interleaved",
            "world_p50_us": round(_pct(w_us, 50), 2), "step_p50_us": round(_pct(s_us, 50), 2),
            "steps": n},
        "world_step_7mm_p99_us": {
            "value": round(_pct(w_us, 99), 2), "unit": "us", "steps": n,
            "step_p99_us": round(_pct(s_us, 99), 2)},
    }
