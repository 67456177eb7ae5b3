"""Benchmarks of the cut plane (:mod:`bonesim.engine.cut_plane`) and of the
irrigated dust step (:mod:`bonesim.physics.dust.water`).

``cut_plane_stroke_ms``
    Wall time of one 20 x 20 mm stroke 5 mm deep into the phantom's lateral
    cortex (:func:`bonesim.engine.cut_plane.publish_cut`: traversal, removal
    and its tissue events), the case reset between strokes (not timed).
``dust_irrigated_step_64_ms``
    Wall time of one :meth:`~bonesim.physics.dust.DustGrid.step` on the
    scene of ``dust_step_64_ms`` (:mod:`bonesim.bench.dust`: a 64^3 box of
    dust in mid-fall on a bone floor, burr and suction inside), with the box
    also holding water (a random amount in [0, 1) per cell) and the
    irrigator pouring at its centre: every rule of the water runs on 64^3
    cells. The plain dust step of the same scene is timed in the same run
    (``dry_step_median_ms``) for comparison.
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ["STROKE_MM", "STROKE_DEPTH_MM", "bench_cut_plane", "bench_irrigated_dust"]

#: Width and height of the benchmark stroke [mm].
STROKE_MM = 20.0
#: Its depth [mm].
STROKE_DEPTH_MM = 5.0
#: Centre of the stroke, 1 mm off the phantom's lateral face [mm]; the rays
#: go along -x.
STROKE_CENTRE_MM = (21.0, 2.0, 0.0)


def bench_cut_plane(quick=False) -> dict:
    """One 20 x 20 mm, 5 mm deep stroke in the phantom (median wall time [ms])."""
    from bonesim.engine.cut_plane import plane_pose, publish_cut
    from bonesim.engine.model import make_state, reset_state
    from bonesim.io.loading import load_model

    model = load_model("phantom", "cutting-5mm")
    state = make_state(model)
    pose = plane_pose(STROKE_CENTRE_MM, (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    publish_cut(state, model.injury, pose, 1.0, 1.0, 1.0, 0.0)        # compile
    n = 10 if quick else 40
    ms = np.empty(n)
    removed = 0
    for q in range(n):
        reset_state(model, state)
        t0 = time.perf_counter()
        removed = publish_cut(state, model.injury, pose, STROKE_MM, STROKE_MM,
                              STROKE_DEPTH_MM, 0.0)
        ms[q] = (time.perf_counter() - t0) * 1e3
    return {"cut_plane_stroke_ms": {
        "value": round(float(np.median(ms)), 3), "unit": "ms",
        "p90_ms": round(float(np.percentile(ms, 90)), 3), "strokes": int(n),
        "voxels_removed": int(removed), "voxel_mm": float(model.grid.spacing_mm),
        "scenario": f"{STROKE_MM:g} x {STROKE_MM:g} mm stroke {STROKE_DEPTH_MM:g} mm deep "
                    "into the phantom's lateral cortex, published as tissue events"}}


def _irrigated_scene(rng):
    from bonesim.bench.dust import EDGE, FLOOR, dust_scene
    from bonesim.physics.dust.grid import Q
    from bonesim.physics.dust.water import water_grid

    bone, dust = dust_scene(rng, full=False)
    ax = [np.arange(8, 8 + EDGE), np.arange(8, 8 + EDGE), np.arange(FLOOR, FLOOR + EDGE)]
    ijk = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    water_grid(dust)._add_q(ijk, (rng.random(len(ijk)) * Q).astype(np.int64))
    return bone, dust


def bench_irrigated_dust(quick=False) -> dict:
    """The irrigated dust step on a 64^3 region, next to the plain one."""
    from bonesim.bench.dust import DT_S, EDGE, FLOOR, time_steps
    from bonesim.physics.dust.grid import warmup

    warmup()
    rng = np.random.default_rng(0)
    n = 60 if quick else 300
    per_reset = 100
    centre = np.array([8 + EDGE / 2, 8 + EDGE / 2, FLOOR + EDGE / 2]) * 0.5    # [mm]
    ms = np.empty(n)
    bone = dust = None
    for q in range(n):
        if q % per_reset == 0:
            bone, dust = _irrigated_scene(rng)
            dust.step(bone, DT_S, irrigation_pos_mm=centre)     # first step: halos
        tool = centre + 6.0 * np.array([np.cos(q * 0.05), np.sin(q * 0.05), 0.0])
        suction = centre + np.array([0.0, 0.0, 8.0])
        t0 = time.perf_counter()
        dust.step(bone, DT_S, tool, 2.5, suction, 1.5, irrigation_pos_mm=centre + (0, 0, 12.0),
                  irrigation_radius_mm=2.0)
        ms[q] = (time.perf_counter() - t0) * 1e3
    dry, _ = time_steps(rng, n, per_reset=per_reset, full=False)
    return {"dust_irrigated_step_64_ms": {
        "value": round(float(np.median(ms)), 3), "unit": "ms",
        "p90_ms": round(float(np.percentile(ms, 90)), 3), "steps": int(n),
        "dry_step_median_ms": round(float(np.median(dry)), 3),
        "ratio_to_dry": round(float(np.median(ms) / np.median(dry)), 2),
        "cells": EDGE ** 3, "dt_s": DT_S,
        "scenario": "the dust_step_64_ms scene with water in every cell of the box (random "
                    "in [0, 1)) and the irrigator pouring above it; dry_step_median_ms: "
                    "the same scene without water, same run"}}


if __name__ == "__main__":                    # pragma: no cover
    import json

    print(json.dumps({**bench_cut_plane(), **bench_irrigated_dust()}, indent=2))
