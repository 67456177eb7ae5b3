"""Benchmark of the Eulerian dust step (:mod:`bonesim.physics.dust.grid`).

``dust_step_64_ms``: wall time of one :meth:`DustGrid.step` on an active
region of 64^3 cells: a 64^3 box of dust resting on a bone floor, every cell
holding a random density in [0, 1) (dust in mid-fall: every cell moves), with
the burr and the suction tip inside the box. The state is rebuilt every
``per_reset`` steps (outside the timing) so that it stays that active.
Figures are wall-clock on whatever machine runs them.
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ["EDGE", "FLOOR", "DT_S", "bench_dust"]

#: Edge of the dusty box [cells].
EDGE = 64
#: Bone floor thickness under the box [cells].
FLOOR = 8
#: Dust step [s].
DT_S = 1e-3


def dust_scene(rng, full: bool):
    from bonesim.physics.dust.grid import DustGrid
    from bonesim.engine.grid import Grid

    shape = (EDGE + 16, EDGE + 16, FLOOR + EDGE + 8)
    lab = np.zeros(shape, np.uint8)
    lab[:, :, :FLOOR] = 1
    bone = Grid.from_dense(lab, spacing_mm=0.5)
    dust = DustGrid.for_grid(bone, (0.0, 0.0, -1.0))
    ax = [np.arange(8, 8 + EDGE), np.arange(8, 8 + EDGE), np.arange(FLOOR, FLOOR + EDGE)]
    ijk = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    amount = np.ones(len(ijk)) if full else rng.random(len(ijk))
    dust.add_removed(ijk, amount)
    return bone, dust


def time_steps(rng, n: int, per_reset: int, full: bool):
    ms = np.empty(n)
    bone = dust = None
    centre = np.array([8 + EDGE / 2, 8 + EDGE / 2, FLOOR + EDGE / 2]) * 0.5   # [mm]
    perf = time.perf_counter
    for q in range(n):
        if q % per_reset == 0:
            bone, dust = dust_scene(rng, full)
            dust.step(bone, DT_S)              # first step allocates the halo
        tool = centre + 6.0 * np.array([np.cos(q * 0.05), np.sin(q * 0.05), 0.0])
        suction = centre + np.array([0.0, 0.0, 8.0])
        t0 = perf()
        dust.step(bone, DT_S, tool, 2.5, suction, 1.5)
        ms[q] = (perf() - t0) * 1e3
    return ms, dust


def bench_dust(quick=False) -> dict:
    """Dust step on a 64^3 active region (median wall time [ms])."""
    from bonesim.physics.dust.grid import warmup

    warmup()
    rng = np.random.default_rng(0)
    n = 60 if quick else 400
    ms, dust = time_steps(rng, n, per_reset=100, full=False)
    ms_full, _ = time_steps(rng, max(20, n // 4), per_reset=100, full=True)
    return {
        "dust_step_64_ms": {
            "value": round(float(np.median(ms)), 3), "unit": "ms",
            "p90_ms": round(float(np.percentile(ms, 90)), 3),
            "min_ms": round(float(ms.min()), 3),
            "steps": int(n), "cells": EDGE ** 3, "dt_s": DT_S,
            "active_bricks": dust.n_active_bricks, "bricks": dust.n_bricks,
            "packed_box_median_ms": round(float(np.median(ms_full)), 3),
            "scenario": "64^3 box of dust, random densities in [0, 1), on a bone floor; "
                        "gravity -z, 2.5 mm burr and 1.5 mm suction inside the box; "
                        "packed_box: the same box full (nothing falls, piles spill)",
        },
    }


if __name__ == "__main__":                    # pragma: no cover
    import json

    print(json.dumps(bench_dust(), indent=2))
