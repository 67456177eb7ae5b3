"""Geometry for the scene: placing the tool, meshing structures (VTK, no state)."""
from __future__ import annotations

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkImageData, vtkPolyData
from vtkmodules.vtkCommonMath import vtkMatrix4x4
from vtkmodules.vtkFiltersCore import (vtkFlyingEdges3D, vtkPolyDataNormals,
                                       vtkWindowedSincPolyDataFilter)

__all__ = ["tool_matrix", "vtk_matrix", "structure_polydata", "polydata_from_arrays", "point_to"]


def tool_matrix(pos_mm, axis, scale=(1.0, 1.0, 1.0)) -> np.ndarray:
    """4x4 placing a model whose +y axis runs along ``-axis`` at ``pos_mm``.

    Parameters
    ----------
    pos_mm : (3,) float
        Origin of the model in the case frame [mm].
    axis : (3,) float
        Drill axis, handle toward burr tip (normalised here).
    scale : (3,) float
        Scale along the model's x, y, z before rotation.
    """
    u = -np.asarray(axis, dtype=float)
    n = np.linalg.norm(u)
    u = u / n if n > 0 else np.array([0.0, 0.0, 1.0])
    h = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(u, h)
    x /= np.linalg.norm(x)
    z = np.cross(x, u)
    m = np.eye(4)
    m[:3, 0] = x * scale[0]
    m[:3, 1] = u * scale[1]
    m[:3, 2] = z * scale[2]
    m[:3, 3] = np.asarray(pos_mm, dtype=float)
    return m


def vtk_matrix(m: np.ndarray) -> vtkMatrix4x4:
    vm = vtkMatrix4x4()
    vm.DeepCopy(m.ravel().tolist())
    return vm


def structure_polydata(mask: np.ndarray, origin_mm, spacing_mm: float,
                       smooth_iterations: int = 15) -> vtkPolyData:
    """Smooth closed surface of a boolean voxel mask.

    Flying edges at level 0.5 on the mask padded by one empty voxel, then a
    windowed-sinc smoothing (no shrinkage) and point normals.

    Parameters
    ----------
    mask : (nx, ny, nz) bool or float
        Voxels of the structure, axes (x, y, z); or the fraction of each
        voxel it fills (0..1, contoured at 0.5).
    origin_mm : (3,) float
        Case-frame centre of ``mask[0, 0, 0]`` [mm].
    spacing_mm : float
        Voxel edge [mm].
    smooth_iterations : int
        Smoothing passes (0: none).
    """
    kind = np.float32 if np.asarray(mask).dtype.kind == "f" else np.uint8
    pad = np.zeros(tuple(s + 2 for s in mask.shape), dtype=kind)
    pad[1:-1, 1:-1, 1:-1] = mask
    img = vtkImageData()
    img.SetDimensions(*pad.shape)
    img.SetSpacing(spacing_mm, spacing_mm, spacing_mm)
    img.SetOrigin(*(np.asarray(origin_mm, dtype=float) - spacing_mm))
    flat = np.ascontiguousarray(pad.transpose(2, 1, 0)).ravel()   # x fastest
    arr = numpy_support.numpy_to_vtk(flat, deep=True)
    arr.SetName("mask")
    img.GetPointData().SetScalars(arr)
    fe = vtkFlyingEdges3D()
    fe.SetInputData(img)
    fe.SetValue(0, 0.5)
    fe.ComputeNormalsOff()
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    src = fe
    if smooth_iterations > 0:
        sm = vtkWindowedSincPolyDataFilter()
        sm.SetInputConnection(fe.GetOutputPort())
        sm.SetNumberOfIterations(int(smooth_iterations))
        sm.SetPassBand(0.1)
        sm.NonManifoldSmoothingOn()
        sm.NormalizeCoordinatesOn()
        sm.BoundarySmoothingOff()
        src = sm
    nm = vtkPolyDataNormals()
    nm.SetInputConnection(src.GetOutputPort())
    nm.SplittingOff()
    nm.ConsistencyOn()
    nm.AutoOrientNormalsOff()
    nm.Update()
    out = vtkPolyData()
    out.DeepCopy(nm.GetOutput())
    return out


def polydata_from_arrays(verts, faces) -> vtkPolyData:
    v = np.ascontiguousarray(verts, dtype=np.float32).reshape(-1, 3)
    f = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    pd = vtkPolyData()
    pts = vtkPoints()
    pts.SetData(numpy_support.numpy_to_vtk(v, deep=True))
    pd.SetPoints(pts)
    cells = vtkCellArray()
    conn = numpy_support.numpy_to_vtkIdTypeArray(f.ravel(), deep=True)
    offs = numpy_support.numpy_to_vtkIdTypeArray(
        np.arange(0, 3 * f.shape[0] + 1, 3, dtype=np.int64), deep=True)
    cells.SetData(offs, conn)
    pd.SetPolys(cells)
    nm = vtkPolyDataNormals()
    nm.SetInputData(pd)
    nm.SplittingOff()
    nm.Update()
    out = vtkPolyData()
    out.DeepCopy(nm.GetOutput())
    return out


def point_to(arr, buf: np.ndarray, n_values: int) -> None:
    """Let VTK array ``arr`` use ``buf``'s memory (its first ``n_values``
    values) in place: ``buf`` must outlive the array's use."""
    arr.SetVoidArray(buf, int(n_values), 1)   # 1: VTK must not free it
    arr.Modified()
