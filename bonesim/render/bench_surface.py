"""Surface benchmarks that need VTK (figures for ``bonesim bench``; never asserted).

:func:`bench_flying_edges` returns

``tessellate_ct512_vs_flying_edges``
    :meth:`bonesim.engine.surface.Surface.build` of the synthetic
    512 x 512 x 300 CT (:func:`bonesim.bench.suite.synthetic_ct`, 0.5 mm)
    over VTK's ``vtkFlyingEdges3D`` contouring the same label volume at
    iso value 0.5 (between empty, 0, and bone, 1), timed alternately in the
    same run (medians). Flying edges runs on VTK's best SMP backend
    available (``STDThread``: one thread per core), computing its normals
    (its default) as our build computes normals and colours. Target <= 1.
``flying_edges_ct512_s``
    The flying-edges time itself (median) [s], with the sequential
    backend's time in the detail.

:func:`bench_native` returns the phantom generated at 0.19 mm (the voxel of
the real temporal-bone stacks, about 274^3 voxels):

``render_update_native_019_ms``
    As ``render_update_1000_ms`` (:func:`bonesim.render.bench.bench_update`):
    surface update plus the push into the scene's buffers, scaled to 1,000
    removed voxels; p99 (p50 in the detail).
``render_fps_native_019``
    As ``render_fps_1024x768`` (:func:`bonesim.render.bench.bench_fps`) while
    drilling: each frame the burr cuts the cavity's floor, the surface and
    scene are updated with the removed voxels, then dust, tool, HUD and
    render. Target >= 20.
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ["NATIVE_VOXEL_MM", "flying_edges", "bench_flying_edges", "bench_native"]

#: Voxel edge of the native-resolution benchmarks [mm] (the real stacks').
NATIVE_VOXEL_MM = 0.19


def flying_edges(labels: np.ndarray, spacing_mm: float, iso: float = 0.5,
                 backend: str = "STDThread"):
    """Contour a label volume with ``vtkFlyingEdges3D``.

    Parameters
    ----------
    labels : (nx, ny, nz) array
        Volume, axis order ``(x, y, z)`` (voxel ``(i, j, k)`` at
        ``spacing_mm * (i, j, k)`` [mm]).
    spacing_mm : float
        Voxel edge [mm].
    iso : float
        Contour value.
    backend : str
        VTK SMP backend (``"STDThread"`` or ``"Sequential"``).

    Returns
    -------
    (seconds, n_points, n_triangles)
        Time of the filter's ``Update`` [s] (the volume is wrapped before),
        and the output's size.
    """
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkSMPTools
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

    img = vtkImageData()
    img.SetDimensions(*labels.shape)
    img.SetSpacing(spacing_mm, spacing_mm, spacing_mm)
    # VTK's point order is x fastest: the (z, y, x) C array, flattened
    flat = np.ascontiguousarray(np.transpose(labels, (2, 1, 0))).ravel()
    img.GetPointData().SetScalars(numpy_to_vtk(flat, deep=True))
    vtkSMPTools.SetBackend(backend)
    fe = vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, iso)
    t0 = time.perf_counter()
    fe.Update()
    dt = time.perf_counter() - t0
    out = fe.GetOutput()
    return dt, int(out.GetNumberOfPoints()), int(out.GetNumberOfCells())


def bench_flying_edges(quick: bool = False) -> dict:
    """``tessellate_ct512_vs_flying_edges`` and ``flying_edges_ct512_s`` (see
    the module docstring)."""
    from vtkmodules.vtkCommonCore import vtkSMPTools

    from bonesim.bench.suite import CT_SHAPE, synthetic_ct
    from bonesim.engine.grid import Grid
    from bonesim.engine.surface import Surface, warmup

    warmup()
    labels = synthetic_ct()
    grid = Grid.from_dense(labels, spacing_mm=0.5)
    colors = np.array([[0, 0, 0], [230, 220, 200]], np.uint8)
    backend = "STDThread"
    reps = 2 if quick else 5
    ours, fe, fe_seq = [], [], []
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
    vtkSMPTools.SetBackend(backend)
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
            "backend": backend, "threads": int(vtkSMPTools.GetEstimatedNumberOfThreads()),
            "sequential_s": round(t_seq, 4), "points": fe_size[0],
            "triangles": fe_size[1], "normals": True},
    }


def bench_native(quick: bool = False, screenshot=None) -> dict:
    """``render_update_native_019_ms`` and ``render_fps_native_019`` (see the
    module docstring); ``screenshot``: PNG path for the last fps frame."""
    from bonesim.render.bench import bench_fps, bench_update

    out = bench_update(quick, voxel_mm=NATIVE_VOXEL_MM, name="render_update_native_019_ms")
    out.update(bench_fps(quick, voxel_mm=NATIVE_VOXEL_MM, name="render_fps_native_019",
                         screenshot=screenshot, drilling=True))
    return out
