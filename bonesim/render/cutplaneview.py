"""The cut plane's rectangle on screen: an outline where the next stroke goes.

The cut-plane tool (:mod:`bonesim.engine.cut_plane`) has no body; the window
shows the rectangle the next stroke will start from as a thin outline, with
a short tick along its normal (the direction the rays go), in
:data:`OUTLINE_RGB`, drawn over the bone (no depth test) so that it is seen
where it enters the bone.
"""
from __future__ import annotations

import numpy as np
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

__all__ = ["OUTLINE_RGB", "OUTLINE_WIDTH_PX", "outline_points", "CutPlaneOutline"]

#: Colour of the outline.
OUTLINE_RGB = (1.0, 0.35, 0.2)
#: Line width [px].
OUTLINE_WIDTH_PX = 2.0


def outline_points(pose, width_mm: float, height_mm: float, depth_mm: float) -> np.ndarray:
    """The rectangle's four corners and the tick's two ends, (6, 3) [mm]:
    corners in order around the rectangle, then the centre and the centre
    moved ``depth_mm`` along the normal."""
    from bonesim.engine.cut_plane import plane_axes

    c = np.asarray(pose[:3], float)
    u, v, n = plane_axes(pose)
    hu, hv = 0.5 * float(width_mm) * u, 0.5 * float(height_mm) * v
    return np.array([c - hu - hv, c + hu - hv, c + hu + hv, c - hu + hv, c,
                     c + float(depth_mm) * n])


class CutPlaneOutline:
    """The outline actor (hidden until :meth:`set` gets a pose).

    Parameters
    ----------
    renderer : vtkRenderer
    """

    def __init__(self, renderer):
        self.polydata = vtkPolyData()
        self._pts = vtkPoints()
        self._pts.SetNumberOfPoints(6)
        lines = vtkCellArray()
        for a, b in ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5)):
            lines.InsertNextCell(2)
            lines.InsertCellPoint(a)
            lines.InsertCellPoint(b)
        self.polydata.SetPoints(self._pts)
        self.polydata.SetLines(lines)
        m = vtkPolyDataMapper()
        m.SetInputData(self.polydata)
        a = vtkActor()
        a.SetMapper(m)
        p = a.GetProperty()
        p.SetColor(*OUTLINE_RGB)
        p.SetLineWidth(OUTLINE_WIDTH_PX)
        p.LightingOff()
        a.SetVisibility(False)
        a.PickableOff()
        renderer.AddActor(a)
        self.actor = a

    def set(self, pose, width_mm=0.0, height_mm=0.0, depth_mm=0.0) -> None:
        """Show the rectangle at ``pose`` (``(cx, cy, cz, qw, qx, qy, qz)``);
        None hides it."""
        if pose is None:
            self.actor.SetVisibility(False)
            return
        for q, p in enumerate(outline_points(pose, width_mm, height_mm, depth_mm)):
            self._pts.SetPoint(q, *p)
        self._pts.Modified()
        self.polydata.Modified()
        self.actor.SetVisibility(True)
