"""Benchmark: a full surface build against VTK's flying edges, in one run.

``tessellate_ct512_vs_flying_edges``
    :meth:`bonesim.engine.surface.Surface.build` of the synthetic
    512 x 512 x 300 CT (:func:`bonesim.bench.suite.synthetic_ct`, 0.5 mm)
    over VTK's ``vtkFlyingEdges3D`` contouring the same label volume at
    iso value 0.5 (between empty, 0, and bone, 1), timed alternately in the
    same run (medians; :func:`bonesim.render.bench_surface.flying_edges`,
    since only ``render/`` imports VTK). Flying edges runs on VTK's
    ``STDThread`` SMP backend (one thread per core, the best this VTK
    offers), computing its normals (its default) as our build computes
    normals and colours. Target <= 1.
``flying_edges_ct512_s``
    The flying-edges time itself (median) [s], with the sequential
    backend's time in the detail.

Figures are reported, never asserted.
"""
from __future__ import annotations

import os
import time

import numpy as np

__all__ = ["bench_flying_edges"]


def bench_flying_edges(quick: bool = False) -> dict:
    """``tessellate_ct512_vs_flying_edges`` and ``flying_edges_ct512_s`` (see
    the module docstring)."""
    from bonesim.bench.suite import CT_SHAPE, synthetic_ct
    from bonesim.render.bench_surface import flying_edges
    from bonesim.engine.grid import Grid
    from bonesim.engine.surface import Surface, warmup

    warmup()
    labels = synthetic_ct()
    grid = Grid.from_dense(labels, spacing_mm=0.5)
    colors = np.array([[0, 0, 0], [230, 220, 200]], np.uint8)
    backend = "STDThread"
    reps = 2 if quick else 5
    ours, fe = [], []
    surf = None
    fe_size = (0, 0)
    for q in range(reps + 1):              # the first round warms both up
        t0 = time.perf_counter()
        surf = Surface.build(grid, colors)
        t_ours = time.perf_counter() - t0
        t_fe, n_pts, n_tri = flying_edges(labels, 0.5, 0.5, backend)
        if q:
            ours.append(t_ours)
            fe.append(t_fe)
            fe_size = (n_pts, n_tri)
    t_seq = flying_edges(labels, 0.5, 0.5, "Sequential")[0]
    flying_edges(labels[:8, :8, :8], 0.5, 0.5, backend)   # leave VTK on that backend
    o, f = float(np.median(ours)), float(np.median(fe))
    return {
        "tessellate_ct512_vs_flying_edges": {
            "value": round(o / f, 3), "unit": "x", "stat": "median / median",
            "what": "Surface.build of the synthetic CT / vtkFlyingEdges3D on the same "
                    "labels at iso 0.5, alternately in one run",
            "ours_s": round(o, 4), "flying_edges_s": round(f, 4), "reps": reps,
            "shape": list(CT_SHAPE), "vertices": int(surf.n_vertices),
            "triangles": int(surf.n_triangles)},
        "flying_edges_ct512_s": {
            "value": round(f, 4), "unit": "s", "stat": "median",
            "backend": backend, "threads": int(os.cpu_count() or 1),
            "sequential_s": round(t_seq, 4), "points": fe_size[0],
            "triangles": fe_size[1], "normals": True},
    }
