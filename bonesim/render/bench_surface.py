"""Surface benchmarks that need VTK (figures for ``bonesim bench``; never asserted).

:func:`flying_edges` times VTK's ``vtkFlyingEdges3D`` on a label volume (for
``tessellate_ct512_vs_flying_edges``, :mod:`bonesim.bench.native_surface`).

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
    render. Target >= 20. The surface is drawn with its level of detail
    (:mod:`bonesim.render.lod`: full detail around the burr and wherever
    bone was drilled, one vertex per 2x2x2 voxels beyond, per 4x4x4 voxels
    of smooth bone beyond ``coarse_mm``), the dust thinned
    (:mod:`bonesim.render.dustview`); the detail's ``lod_second_level``
    says whether the second level was on.
"""
from __future__ import annotations

import time

import numpy as np

__all__ = ["NATIVE_VOXEL_MM", "flying_edges", "bench_native"]

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


def bench_native(quick: bool = False, screenshot=None) -> dict:
    """``render_update_native_019_ms`` and ``render_fps_native_019`` (see the
    module docstring); ``screenshot``: PNG path for the last fps frame."""
    from bonesim.io.loading import load_model
    from bonesim.render.bench import bench_fps, bench_update

    # the 0.19 mm phantom is built once for both (20 million voxels)
    model = load_model("phantom", "cutting-5mm", voxel_mm=NATIVE_VOXEL_MM)
    out = bench_update(quick, voxel_mm=NATIVE_VOXEL_MM, name="render_update_native_019_ms",
                       model=model)
    out.update(bench_fps(quick, voxel_mm=NATIVE_VOXEL_MM, name="render_fps_native_019",
                         screenshot=screenshot, drilling=True, model=model))
    return out
